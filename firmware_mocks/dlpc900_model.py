"""The DLPC900 controller as a state machine, written from the programmer's guide (DLPU018).

This is the device side only: it takes one complete command (flags, sequence, opcode, payload)
and answers with a reply payload or an error code, exactly as `protocols.md` describes. The USB
framing lives in `dlpc900_usb.py`. Nothing here imports `drivers`: the image decoder below is
written from the specification, so a driver whose encoder is wrong fails against it.

Time comes from an injectable clock (ns), so tests can step the ~300 ms display-mode settle and
the pattern timeline without sleeping.
"""

from __future__ import annotations

import bisect

import struct
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

# Error codes (0x0100) and the descriptions the emulated firmware reports on 0x0101.
ERR_NONE = 0
ERR_DEVICE_FAILURE = 2
ERR_INVALID_COMMAND = 3
ERR_NOT_ALLOWED = 5
ERR_INVALID_PARAMETER = 6
ERR_ITEM_NOT_PRESENT = 7
ERR_OUT_OF_MEMORY = 8
ERR_INVALID_COMPRESSION = 9
ERR_BIT_OUT_OF_RANGE = 10
ERR_DARK_TIME = 12
ERR_SIGNAL_DELAY = 13
ERR_EXPOSURE = 14
ERR_PATTERN_NUMBER = 15
ERR_PATTERN_DEFINITION = 16
ERR_IMAGE_ADDRESS = 17
ERR_INTERNAL = 255

ERROR_NAMES = {
    0: "no error", 1: "batch file checksum error", 2: "device failure", 3: "invalid command number",
    4: "incompatible controller and DMD", 5: "command not allowed in current mode",
    6: "invalid command parameter", 7: "item referred by the parameter is not present",
    8: "out of resource (RAM or flash)", 9: "invalid BMP compression type", 10: "pattern bit number out of range",
    11: "pattern BMP not present in flash", 12: "pattern dark time out of range",
    13: "signal delay parameter out of range", 14: "pattern exposure time out of range",
    15: "pattern number out of range", 16: "invalid pattern definition", 17: "pattern image memory address out of range",
    255: "internal error",
}

# Minimum exposure (µs) per bit depth for a DLP6500. 1, 2, 4, 8 bits from protocols.md; the
# others from the DLPC900 datasheet's pattern-rate table (DLP6500, no LED modulation).
MIN_EXPOSURE_US = {1: 105, 2: 304, 3: 394, 4: 823, 5: 1215, 6: 1487, 7: 1998, 8: 4046}
# DLPU018 (0x1A1B): once sync is locked, the switch to video pattern mode (2) takes about 300 ms,
# and reading the mode back sooner may not return it. It names no such delay for the other modes.
SETTLE_NS = 300_000_000
SETTLING_MODES = {2}
MAX_IMAGE_INDEX = 255  # image pattern index is bits 10:0 but the guide limits it to 0..255

# DMD type (0x0206) -> native resolution. The DLP9000 is driven by two DLPC900s, each holding one
# half of every pattern image (DLPU018: the primary the left half, the secondary the right).
DMD_RESOLUTION = {1: (1920, 1080), 2: (2560, 1600)}
DUAL_CONTROLLER_DMDS = {2}
HW_SECONDARY_PRESENT = 0x10  # hardware status (0x1A0A) bit 4

RESET_LED_ENABLE = 0x08
RESET_LED_CURRENT = (0x97, 0x78, 0x7D)


class RecentLog(list):
    """A list for the emulator's records that keeps only the newest entries.

    The mock also runs for whole sessions (`dpmhw run --mock` polls its status every few
    seconds), so its logs must not grow without bound; tests read them as plain lists. Past
    `limit` entries the oldest half is dropped at once, which keeps `append` amortised O(1).
    """

    def __init__(self, limit: int = 100_000):
        super().__init__()
        self.limit = limit

    def append(self, item) -> None:
        super().append(item)
        self._trim()

    def extend(self, items) -> None:
        super().extend(items)
        self._trim()

    def _trim(self) -> None:
        if len(self) > self.limit:
            del self[: len(self) - self.limit // 2]


class CommandError(Exception):
    """A command the controller rejects; carries the 0x0100 code and 0x0101 text."""

    def __init__(self, code: int, description: str | None = None):
        self.code = code
        self.description = description or ERROR_NAMES.get(code, "error")
        super().__init__(f"{code}: {self.description}")


@dataclass
class LoggedCommand:
    t_ns: int
    seq: int
    opcode: int
    read: bool
    reply_wanted: bool
    data: bytes
    error: int  # 0 = accepted


@dataclass(frozen=True)
class LutEntry:
    """One pattern-LUT definition (0x1A34), decoded."""

    index: int
    exposure_us: int
    clear_after: bool
    bit_depth: int
    color: int
    wait_trigger: bool
    dark_us: int
    disable_trigger_out2: bool
    image_index: int
    bit_position: int


def video_frame_groups(entries: list[LutEntry]) -> list[list[LutEntry]]:
    """The LUT split into what one video frame shows in video pattern mode: a group starts at
    an entry that waits for the trigger (the frame's VSYNC) and runs to the next. A LUT in
    which no entry waits starts its one group at every VSYNC (an assumption: DLPU018 does
    not say what the sequencer does then)."""
    groups: list[list[LutEntry]] = []
    for e in entries:
        if e.wait_trigger or not groups:
            groups.append([])
        groups[-1].append(e)
    return groups


@dataclass(frozen=True)
class DisplayedPattern:
    """One pattern the DMD showed: when, which LUT entry, which bits of which image."""

    t_ns: int
    lut_index: int
    image_index: int
    bit_position: int
    bit_depth: int
    exposure_us: int


class ImageDecodeError(ValueError):
    def __init__(self, message: str, code: int = ERR_INVALID_COMPRESSION):
        self.code = code
        super().__init__(message)


HEADER_SIZE = 48
# Zero bytes after the end of the image that the controller ignores, per compression: a public
# host pads every image to a 4-byte boundary, TI's reference plain-RLE encoder to a 16-byte one.
MAX_PADDING = {0: 3, 1: 15, 2: 3}


def _read_count(buf: bytes, i: int) -> tuple[int, int]:
    b0 = buf[i]
    if b0 < 0x80:
        return b0, i + 1
    if i + 1 >= len(buf):
        raise ImageDecodeError("count byte truncated")
    return (b0 & 0x7F) | (buf[i + 1] << 7), i + 2


# A pixel's three bytes come most significant first: the last one holds bit positions 0-7, as
# hardware-proven hosts send them (docs/projector.md).
def _pixel(buf: bytes, at: int) -> int:
    return (buf[at] << 16) | (buf[at + 1] << 8) | buf[at + 2]


def _pixels(raw: np.ndarray, at: int, n: int) -> np.ndarray:
    b = raw[at:at + 3 * n].reshape(n, 3).astype(np.uint32)
    return (b[:, 0] << 16) | (b[:, 1] << 8) | b[:, 2]


def decode_pattern_image(blob: bytes) -> np.ndarray:
    """Header + payload -> (H, W) uint32 image, as the controller would unpack it.

    Tolerated, because hardware-proven hosts send them (docs/projector.md): a header byte count
    (offset 8) that is either the payload's length or the whole image's (header included), and
    zero padding after the end of the image (up to 3 bytes; 15 for plain RLE). Raises
    ImageDecodeError for a bad signature, an unknown compression, a line that over- or under-runs
    the width, a copy on the first line, a missing end-of-image, trailing lines, or anything else
    after the image.
    """
    if len(blob) < HEADER_SIZE:
        raise ImageDecodeError(f"image shorter than its 48-byte header ({len(blob)} bytes)")
    if blob[:4] != b"Spld":
        raise ImageDecodeError("bad image signature (expected 'Spld')")
    width, height, nbytes = struct.unpack_from("<HHI", blob, 4)
    compression = blob[25]
    payload = blob[HEADER_SIZE:]
    if width == 0 or height == 0:
        raise ImageDecodeError("zero image size", ERR_INVALID_PARAMETER)
    if compression == 0:
        end = 3 * width * height
        if len(payload) < end:
            raise ImageDecodeError(f"uncompressed image has {len(payload)} data bytes, "
                                   f"{width}x{height}x3 = {end} needed")
        img = _pixels(np.frombuffer(payload, np.uint8), 0, width * height).reshape(height, width)
    elif compression == 1:
        img, end = _decode_rle(payload, width, height)
    elif compression == 2:
        img, end = _decode_erle(payload, width, height)
    else:
        raise ImageDecodeError(f"compression {compression} (expected 0 none, 1 RLE or 2 enhanced RLE)")
    tail = payload[end:]
    if len(tail) > MAX_PADDING[compression] or any(tail):
        raise ImageDecodeError(f"{len(tail)} bytes after the end of the image (at most "
                               f"{MAX_PADDING[compression]} zero bytes of padding are accepted)", ERR_INVALID_PARAMETER)
    accepted = {end, len(payload), HEADER_SIZE + end, HEADER_SIZE + len(payload)}
    if nbytes not in accepted:
        raise ImageDecodeError(f"header byte count {nbytes} matches neither the {end}-byte image data "
                               f"nor the {HEADER_SIZE + end}-byte image with its header", ERR_INVALID_PARAMETER)
    return img


def _decode_rle(buf: bytes, width: int, height: int) -> tuple[np.ndarray, int]:
    """Compression 1 (DLPU018 "24-bit RLE"): `n pixel` repeats (n = 1..255), `00 c` + c pixels
    uncompressed (c >= 2), `00 00` end of line, `00 01` end of image. Every line starts on a
    4-byte boundary: after an end of line the controller skips to the next multiple of 4, so the
    bytes in between (padding) are not read. Returns the image and the offset after end-of-image."""
    out = np.zeros((height, width), dtype=np.uint32)
    raw = np.frombuffer(buf, dtype=np.uint8)
    n_bytes = len(buf)
    y = x = i = 0
    while True:
        if i >= n_bytes:
            raise ImageDecodeError("image data ended without the end-of-image code (00 01)")
        n = buf[i]
        if n:  # repeat the next pixel n times
            if i + 4 > n_bytes:
                raise ImageDecodeError("repeat token truncated")
            if y >= height or x + n > width:
                raise ImageDecodeError(f"repeat of {n} overruns line {y} at column {x}")
            out[y, x:x + n] = _pixel(buf, i + 1)
            x, i = x + n, i + 4
            continue
        if i + 1 >= n_bytes:
            raise ImageDecodeError("control code truncated")
        c = buf[i + 1]
        if c == 0:  # end of line; the next line starts at the next 4-byte boundary
            if x != width:
                raise ImageDecodeError(f"line {y} ended after {x} of {width} pixels")
            y, x, i = y + 1, 0, (i + 2 + 3) & ~3
            continue
        if c == 1:  # end of image
            if x == width:  # the last line may end with end-of-image instead of 00 00
                y, x = y + 1, 0
            if x != 0 or y != height:
                raise ImageDecodeError(f"end of image after {y} of {height} lines")
            return out, i + 2
        if i + 2 + 3 * c > n_bytes:
            raise ImageDecodeError("uncompressed block truncated")
        if y >= height or x + c > width:
            raise ImageDecodeError(f"uncompressed block of {c} overruns line {y} at column {x}")
        out[y, x:x + c] = _pixels(raw, i + 2, c)
        x, i = x + c, i + 2 + 3 * c


def _decode_erle(buf: bytes, width: int, height: int) -> tuple[np.ndarray, int]:
    """Compression 2 (enhanced RLE); returns the image and the offset after end-of-image."""
    out = np.zeros((height, width), dtype=np.uint32)
    raw = np.frombuffer(buf, dtype=np.uint8)
    y = x = 0
    i = 0
    n_bytes = len(buf)
    while True:
        if i >= n_bytes:
            raise ImageDecodeError("image data ended without the end-of-image code (00 01 00)")
        if buf[i] != 0:  # repeat
            n, i = _read_count(buf, i)
            if i + 3 > n_bytes:
                raise ImageDecodeError("repeat token truncated")
            if y >= height or x + n > width:
                raise ImageDecodeError(f"repeat of {n} overruns line {y} at column {x}")
            out[y, x:x + n] = (buf[i] << 16) | (buf[i + 1] << 8) | buf[i + 2]  # as _pixel, inlined: per token
            x += n
            i += 3
            continue
        if i + 1 >= n_bytes:
            raise ImageDecodeError("control code truncated")
        c = buf[i + 1]
        if c == 0:  # end of line
            if x != width:
                raise ImageDecodeError(f"line {y} ended after {x} of {width} pixels")
            y, x, i = y + 1, 0, i + 2
            continue
        if c == 1:  # copy from previous line, or end of image
            if i + 2 >= n_bytes:
                raise ImageDecodeError("copy / end-of-image code truncated")
            n, j = _read_count(buf, i + 2)
            if n == 0:
                if x == width:  # tolerate a last line not closed by 00 00
                    y, x = y + 1, 0
                if x != 0 or y != height:
                    raise ImageDecodeError(f"end of image after {y} of {height} lines")
                return out, j
            if y == 0:
                raise ImageDecodeError("copy from the previous line on the first line")
            if y >= height or x + n > width:
                raise ImageDecodeError(f"copy of {n} overruns line {y} at column {x}")
            out[y, x:x + n] = out[y - 1, x:x + n]
            x, i = x + n, j
            continue
        n, j = _read_count(buf, i + 1)  # uncompressed block of n >= 2 pixels
        if j + 3 * n > n_bytes:
            raise ImageDecodeError("uncompressed block truncated")
        if y >= height or x + n > width:
            raise ImageDecodeError(f"uncompressed block of {n} overruns line {y} at column {x}")
        out[y, x:x + n] = _pixels(raw, j, n)
        x, i = x + n, j + 3 * n


@dataclass
class _ImageLoad:
    index: int
    expected: int
    secondary: bool
    buf: bytearray = field(default_factory=bytearray)


class DLPC900Model:
    """Controller state and command semantics.

    `execute(opcode, data, read)` returns the reply payload or raises CommandError; the USB layer
    turns that into reply reports and latches the error code for 0x0100.

    With a two-controller DMD (`dmd_type=2`, DLP9000) the model is the pair: 0x1A2A/0x1A2B load
    the primary's half (the left `width // 2` columns) into `images`, 0x1A2C/0x1A2D the
    secondary's (the right half) into `images_secondary`; a sequence needs both halves.
    `width` and `height` default to the DMD type's native resolution.
    """

    def __init__(self, *, width: int | None = None, height: int | None = None, dmd_type: int = 1,
                 tag: str = "DLPC900 emulator", clock: Callable[[], int] = time.monotonic_ns,
                 firmware: tuple[tuple[int, int, int], ...] = ((5, 3, 0), (5, 1, 0), (2, 0, 0), (3, 1, 0))):
        native = DMD_RESOLUTION.get(dmd_type, DMD_RESOLUTION[1])
        self.width = native[0] if width is None else width
        self.height = native[1] if height is None else height
        self.dmd_type = dmd_type
        self.tag = tag
        self.clock = clock
        self.firmware = firmware  # (major, minor, patch) for application, API, sw config, seq config
        self.command_log: RecentLog = RecentLog()  # LoggedCommand per command
        self.events: RecentLog = RecentLog()  # (t_ns, what) for sequencer and mode changes
        self.trigger_times: list[int] = []  # external trigger-in edges (tests add them)
        # The video input's frame period while a source drives it with valid syncs (set by the
        # video cable's device side, `firmware_mocks.video_link`), else None. Not reset by power-on:
        # the source outside keeps sending.
        self.video_period_ns: int | None = None
        self.power_on()

    # ---- state -------------------------------------------------------------------------
    def power_on(self) -> None:
        """Power-on defaults: video mode, sequencer stopped, LEDs under sequencer control."""
        self.standby = False
        self.idle = False
        self.parked = False
        self.display_mode = 0
        self._mode_from = 0
        self._mode_settled_at = 0
        self.sequencer = "stopped"  # stopped | running | paused
        self._run_started_at: int | None = None
        self.led_enable = RESET_LED_ENABLE
        self.led_current = RESET_LED_CURRENT
        self.curtain = (0, 0, 0)
        self.input_source = 0
        self.trigger_out = {1: (0, 0, 0), 2: (0, 0, 0)}
        self.trigger_in1_delay = 104
        self.trigger_in2_polarity = 0
        self.lut: dict[int, LutEntry] = {}
        self.lut_config: tuple[int, int] | None = None  # (entries, repeat)
        self._lut_dirty = False
        self.images: dict[int, np.ndarray] = {}
        self.images_secondary: dict[int, np.ndarray] = {}
        self._loads: dict[bool, _ImageLoad | None] = {False: None, True: None}  # per controller
        self.hw_status = 0x01 | (HW_SECONDARY_PRESENT if self.dual_controller else 0)  # init OK
        self.error_code = 0
        self.error_description = ""
        self._timeline: RecentLog = RecentLog()  # DisplayedPattern of finished runs
        self._dark_changes: RecentLog = RecentLog(1000)  # (t_ns, dark) whenever `dark` changed
        self._note_dark()

    @property
    def run_started_ns(self) -> int | None:
        """When the running pattern sequence started (None unless one runs)."""
        return self._run_started_at

    @property
    def dual_controller(self) -> bool:
        return self.dmd_type in DUAL_CONTROLLER_DMDS

    @property
    def image_width(self) -> int:
        """Width of the images one controller holds: half the DMD on a two-controller DMD."""
        return self.width // 2 if self.dual_controller else self.width

    @property
    def dark(self) -> bool:
        """True when no light reaches the DMD output: standby, idle, parked or LEDs off."""
        leds = self.led_enable & 0x07 or (self.led_enable & 0x08 and self._sequencer_lights())
        return self.standby or self.idle or self.parked or not leds

    def dark_at(self, t_ns: int) -> bool:
        """`dark` as it was at `t_ns`, from the commands' record (the video side scans out
        refreshes after the fact, and a refresh the projector spent dark must stay dark)."""
        changes = self._dark_changes
        k = bisect.bisect_right(changes, (t_ns, True)) - 1
        if k < 0 or k == len(changes) - 1:  # since the last command: as it is now
            return self.dark
        return changes[k][1]

    def _note_dark(self) -> None:
        d = self.dark
        if not self._dark_changes or self._dark_changes[-1][1] != d:
            self._dark_changes.append((self.clock(), d))

    def _sequencer_lights(self) -> bool:
        # With the sequencer in control, light flows in video mode or while a pattern runs.
        return self.display_mode == 0 or self.sequencer == "running"

    def main_status(self) -> int:
        locked = self.video_period_ns is not None  # bit 3 external source locked, bit 4 port 1 syncs valid
        return int(self.parked) | (int(self.sequencer == "running") << 1) | (int(locked) << 3) | (int(locked) << 4)

    @property
    def settled_display_mode(self) -> int:
        return self.display_mode if self.clock() >= self._mode_settled_at else self._mode_from

    # ---- faults tests can raise from the device side -------------------------------------
    def abort_sequence(self) -> None:
        """Sequencer abort: the hardware-status abort bit sets and the sequence stops."""
        self.hw_status |= 0x40
        self._stop("abort")
        self._note_dark()

    def trigger(self, t_ns: int | None = None) -> None:
        self.trigger_times.append(self.clock() if t_ns is None else t_ns)

    # ---- the command set ----------------------------------------------------------------
    STANDBY_ALLOWED = {0x0100, 0x0101, 0x0200, 0x1A0A, 0x1A0B, 0x1A0C}

    def execute(self, opcode: int, data: bytes, read: bool) -> bytes:
        if self.standby and opcode not in self.STANDBY_ALLOWED:
            raise CommandError(ERR_NOT_ALLOWED, "controller is in standby: only wake (0x0200 = 0) is accepted")
        spec = _COMMANDS.get(opcode)
        if spec is None:
            raise CommandError(ERR_INVALID_COMMAND, f"unknown command 0x{opcode:04X}")
        reader, writer, sizes = spec
        if read:
            if reader is None:
                raise CommandError(ERR_INVALID_COMMAND, f"command 0x{opcode:04X} cannot be read")
            return reader(self)
        if writer is None:
            raise CommandError(ERR_INVALID_COMMAND, f"command 0x{opcode:04X} is read-only")
        if sizes is not None and len(data) not in sizes:
            raise CommandError(ERR_INVALID_PARAMETER,
                               f"command 0x{opcode:04X} takes {sorted(sizes)} data bytes, got {len(data)}")
        writer(self, data)
        self._note_dark()
        return b""

    # reads
    def _r_error(self) -> bytes:
        return bytes([self.error_code])

    def _r_error_desc(self) -> bytes:
        return self.error_description.encode("ascii", "replace")[:127] + b"\x00"

    def _r_power(self) -> bytes:
        return bytes([1 if self.standby else 0])

    def _r_idle(self) -> bytes:
        return bytes([int(self.idle)])

    def _r_version(self) -> bytes:
        return b"".join(struct.pack("<HBB", p, mi, ma) for ma, mi, p in self.firmware)

    def _r_hwconfig(self) -> bytes:
        return bytes([self.dmd_type]) + self.tag.encode("ascii")[:31].ljust(31, b"\x00")

    def _r_park(self) -> bytes:
        return bytes([int(self.parked)])

    def _r_curtain(self) -> bytes:
        return struct.pack("<3H", *self.curtain)

    def _r_source(self) -> bytes:
        return bytes([self.input_source])

    def _r_led_enable(self) -> bytes:
        return bytes([self.led_enable])

    def _r_hw_status(self) -> bytes:
        return bytes([self.hw_status])

    def _r_sys_status(self) -> bytes:
        return b"\x01"

    def _r_main_status(self) -> bytes:
        return bytes([self.main_status()])

    def _r_display_mode(self) -> bytes:
        return bytes([self.settled_display_mode])

    def _r_trig_out(self, n: int) -> bytes:
        inv, rise, fall = self.trigger_out[n]
        return struct.pack("<Bhh", inv, rise, fall)

    def _r_pattern(self) -> bytes:
        return bytes([{"stopped": 0, "paused": 1, "running": 2}[self.sequencer]])

    def _r_lut_config(self) -> bytes:
        n, rep = self.lut_config or (0, 0)
        return struct.pack("<HI", n, rep)

    def _r_trig_in1(self) -> bytes:
        return struct.pack("<H", self.trigger_in1_delay)

    def _r_trig_in2(self) -> bytes:
        return bytes([self.trigger_in2_polarity])

    def _r_led_current(self) -> bytes:
        return bytes(self.led_current)

    # writes
    def _w_power(self, d: bytes) -> None:
        mode = d[0]
        if mode == 0:
            self.standby = False
        elif mode == 1:
            self._stop("standby")
            self.standby = True
        elif mode == 2:
            self.power_on()
            self.events.append((self.clock(), "software reset"))
        else:
            raise CommandError(ERR_INVALID_PARAMETER, f"power mode {mode} (expected 0, 1 or 2)")

    def _w_idle(self, d: bytes) -> None:
        if d[0] & 0xFE:
            raise CommandError(ERR_INVALID_PARAMETER, "idle mode: only bit 0 is defined")
        on = bool(d[0] & 1)
        if on and self.sequencer != "stopped":
            raise CommandError(ERR_NOT_ALLOWED, "stop the pattern sequence before entering idle mode")
        self.idle = on
        self.events.append((self.clock(), "idle on" if on else "idle off"))

    def _w_park(self, d: bytes) -> None:
        if d[0] not in (0, 1):
            raise CommandError(ERR_INVALID_PARAMETER, "park: 1 park, 0 unpark")
        self.parked = bool(d[0])

    def _w_curtain(self, d: bytes) -> None:
        rgb = struct.unpack("<3H", d)
        if max(rgb) > 0x3FF:
            raise CommandError(ERR_INVALID_PARAMETER, "curtain colour is 10 bits per channel")
        self.curtain = rgb

    def _w_source(self, d: bytes) -> None:
        if d[0] & 0x07 > 3 or d[0] & 0xE0:
            raise CommandError(ERR_INVALID_PARAMETER, f"input source byte 0x{d[0]:02X}")
        self.input_source = d[0]

    def _w_led_enable(self, d: bytes) -> None:
        if d[0] & 0xF0:
            raise CommandError(ERR_INVALID_PARAMETER, "LED enable: bits 7:4 are reserved")
        self.led_enable = d[0]

    def _w_display_mode(self, d: bytes) -> None:
        mode = d[0]
        if mode > 3:
            raise CommandError(ERR_INVALID_PARAMETER, f"display mode {mode} (expected 0..3)")
        if self.sequencer != "stopped":
            raise CommandError(ERR_NOT_ALLOWED, "stop the pattern sequence before changing the display mode")
        if mode == 2 and mode != self.display_mode and (self.settled_display_mode != 0 or self.video_period_ns is None):
            # DLPU018 (0x1A1B): video pattern mode only from video mode, with the source's sync locked
            raise CommandError(ERR_NOT_ALLOWED, "video pattern mode needs video mode with a locked video source first")
        if mode != self.display_mode:
            self._mode_from = self.settled_display_mode
            self.display_mode = mode
            self._mode_settled_at = self.clock() + (SETTLE_NS if mode in SETTLING_MODES else 0)
            self.lut.clear()
            self.lut_config = None
            self.events.append((self.clock(), f"display mode {mode}"))

    def _w_trig_out(self, n: int, d: bytes) -> None:
        inv, rise, fall = struct.unpack("<Bhh", d)
        if inv > 1:
            raise CommandError(ERR_INVALID_PARAMETER, "trigger out invert: 0 or 1")
        if not (-20 <= rise <= 20000 and -20 <= fall <= 20000):
            raise CommandError(ERR_SIGNAL_DELAY, f"trigger out {n} delay out of -20..20000 µs")
        self.trigger_out[n] = (inv, rise, fall)

    def _w_pattern(self, d: bytes) -> None:
        what = d[0]
        if what not in (0, 1, 2):
            raise CommandError(ERR_INVALID_PARAMETER, "pattern start/stop: 0 stop, 1 pause, 2 start")
        if what == 0:
            self._stop("stop")
            return
        if self.display_mode == 0:
            raise CommandError(ERR_NOT_ALLOWED, "no pattern sequence in video mode")
        if what == 1:
            if self.sequencer == "running":
                self._close_timeline()
                self.sequencer = "paused"
                self.events.append((self.clock(), "pause"))
            return
        if self.idle:
            raise CommandError(ERR_NOT_ALLOWED, "controller is in idle mode")
        if self.clock() < self._mode_settled_at:
            raise CommandError(ERR_NOT_ALLOWED, "display mode switch still in progress")
        if self.lut_config is None or self._lut_dirty:
            raise CommandError(ERR_PATTERN_DEFINITION, "LUT must be configured (0x1A31) after its definitions")
        n, _ = self.lut_config
        for k in range(n):
            e = self.lut[k]
            if self.display_mode == 3 and e.image_index not in self.images:
                raise CommandError(ERR_ITEM_NOT_PRESENT, f"LUT entry {k} names image {e.image_index}, not loaded")
            if self.display_mode == 3 and self.dual_controller and e.image_index not in self.images_secondary:
                raise CommandError(ERR_ITEM_NOT_PRESENT,
                                   f"LUT entry {k} names image {e.image_index}, not loaded on the secondary controller")
        if self.sequencer != "running":
            self.sequencer = "running"
            self.hw_status &= ~0x40
            self._run_started_at = self.clock()
            self.events.append((self.clock(), "start"))

    def _stop(self, why: str) -> None:
        if self.sequencer != "stopped":
            if self.sequencer == "running":
                self._close_timeline()
            self.sequencer = "stopped"
            self.events.append((self.clock(), why))

    def _w_image_init(self, secondary: bool, d: bytes) -> None:
        index, size = struct.unpack("<HI", d)
        if self.display_mode != 3:
            raise CommandError(ERR_NOT_ALLOWED, "image load needs pattern on-the-fly mode (3)")
        if self.sequencer != "stopped":
            raise CommandError(ERR_NOT_ALLOWED, "stop the sequence before loading images")
        if secondary and not self.dual_controller:
            raise CommandError(ERR_NOT_ALLOWED, "no secondary controller: this DMD has one DLPC900")
        if index > MAX_IMAGE_INDEX:
            raise CommandError(ERR_IMAGE_ADDRESS, f"image index {index} > {MAX_IMAGE_INDEX}")
        if size < 48 or size > 48 + 4 * self.image_width * self.height + 5 * self.height + 3:
            raise CommandError(ERR_OUT_OF_MEMORY, f"image of {size} bytes does not fit")
        self._loads[secondary] = _ImageLoad(index, size, secondary)

    def _w_image_data(self, secondary: bool, d: bytes) -> None:
        if len(d) < 2:
            raise CommandError(ERR_INVALID_PARAMETER, "image data: missing byte count")
        n = struct.unpack_from("<H", d)[0] & 0x3FF
        chunk = d[2:]
        if n != len(chunk) or n > 504:
            raise CommandError(ERR_INVALID_PARAMETER, f"image data: count {n} but {len(chunk)} bytes (max 504)")
        load = self._loads[secondary]
        if load is None:
            init = 0x1A2C if secondary else 0x1A2A
            raise CommandError(ERR_NOT_ALLOWED, f"image data without a load init (0x{init:04X})")
        if len(load.buf) + n > load.expected:
            self._loads[secondary] = None
            raise CommandError(ERR_INVALID_PARAMETER, "more image data than announced")
        load.buf += chunk
        if len(load.buf) == load.expected:
            self._loads[secondary] = None
            try:
                img = decode_pattern_image(bytes(load.buf))
            except ImageDecodeError as exc:
                raise CommandError(exc.code, str(exc)) from None
            want = (self.image_width, self.height)
            if (img.shape[1], img.shape[0]) != want:
                half = " (half of a two-controller DMD)" if self.dual_controller else ""
                raise CommandError(ERR_INVALID_PARAMETER,
                                   f"image is {img.shape[1]}x{img.shape[0]}, expected {want[0]}x{want[1]}{half}")
            (self.images_secondary if secondary else self.images)[load.index] = img
            self.events.append((self.clock(), f"{'secondary ' if secondary else ''}image {load.index} loaded"))

    def _w_lut_config(self, d: bytes) -> None:
        n, repeat = struct.unpack("<HI", d)
        if self.display_mode == 0:
            raise CommandError(ERR_NOT_ALLOWED, "LUT configuration needs a pattern display mode")
        if n == 0 or any(k not in self.lut for k in range(n)):
            raise CommandError(ERR_PATTERN_NUMBER, f"{n} entries configured but not all are defined")
        if self.display_mode == 2:
            self._check_video_frame_fits([self.lut[k] for k in range(n)])
        self.lut_config = (n, repeat)
        self._lut_dirty = False

    def _check_video_frame_fits(self, entries: list[LutEntry]) -> None:
        """Video pattern mode shows the patterns of one video frame within that frame: each run
        of entries from one that waits for the trigger (the frame's VSYNC) to the next must
        expose and darken within the input's frame period. DLPU018 states no such check; the
        rule is the one TI's DLPC347x datasheets give for their equivalent 8-bit external
        pattern mode, and error 14 (exposure out of range) the code that names it."""
        if self.video_period_ns is None:
            raise CommandError(ERR_NOT_ALLOWED, "video pattern mode has lost its video source")
        for group in video_frame_groups(entries):
            total_us = sum(e.exposure_us + e.dark_us for e in group)
            if total_us * 1000 > self.video_period_ns:
                raise CommandError(ERR_EXPOSURE, f"LUT entries {group[0].index}..{group[-1].index} take {total_us} µs, "
                                                 f"more than the {self.video_period_ns / 1000:.0f} µs video frame period")

    def _w_lut_define(self, d: bytes) -> None:
        index = struct.unpack_from("<H", d, 0)[0]
        exposure = int.from_bytes(d[2:5], "little")
        opts = d[5]
        dark = int.from_bytes(d[6:9], "little")
        trig2 = d[9]
        img_word = struct.unpack_from("<H", d, 10)[0]
        if self.display_mode == 0:
            raise CommandError(ERR_NOT_ALLOWED, "set a pattern display mode before defining the LUT")
        if self.sequencer != "stopped":
            raise CommandError(ERR_NOT_ALLOWED, "stop the sequence before changing the LUT")
        depth = ((opts >> 1) & 0x07) + 1
        entry = LutEntry(index=index, exposure_us=exposure, clear_after=bool(opts & 1), bit_depth=depth,
                         color=(opts >> 4) & 0x07, wait_trigger=bool(opts & 0x80), dark_us=dark,
                         disable_trigger_out2=bool(trig2 & 1), image_index=img_word & 0x7FF,
                         bit_position=img_word >> 11)
        if index >= 400:
            raise CommandError(ERR_PATTERN_NUMBER, f"pattern index {index} out of range")
        if exposure < MIN_EXPOSURE_US[depth]:
            raise CommandError(ERR_EXPOSURE, f"{exposure} µs is below the {MIN_EXPOSURE_US[depth]} µs minimum for {depth}-bit")
        if entry.bit_position > 23 or entry.bit_position + depth > 24 or entry.bit_position % depth:
            raise CommandError(ERR_BIT_OUT_OF_RANGE, f"bit position {entry.bit_position} for {depth}-bit patterns")
        if entry.image_index > MAX_IMAGE_INDEX:
            raise CommandError(ERR_IMAGE_ADDRESS, f"image index {entry.image_index}")
        self.lut[index] = entry
        self._lut_dirty = True

    def _w_trig_in1(self, d: bytes) -> None:
        (delay,) = struct.unpack("<H", d)
        if delay < 104:
            raise CommandError(ERR_SIGNAL_DELAY, f"trigger in 1 delay {delay} µs is below 104 µs")
        self.trigger_in1_delay = delay

    def _w_trig_in2(self, d: bytes) -> None:
        if d[0] > 1:
            raise CommandError(ERR_INVALID_PARAMETER, "trigger in 2 polarity: 0 or 1")
        self.trigger_in2_polarity = d[0]

    def _w_led_current(self, d: bytes) -> None:
        self.led_current = tuple(d)

    # ---- what the DMD showed ------------------------------------------------------------
    def dmd_image(self, image_index: int) -> np.ndarray:
        """(H, W) uint32 image across the whole DMD: on a two-controller DMD the primary's half
        on the left, the secondary's on the right."""
        if not self.dual_controller:
            return self.images[image_index]
        return np.hstack([self.images[image_index], self.images_secondary[image_index]])

    def dmd_pattern(self, lut_index: int) -> np.ndarray:
        """(H, W) uint8 values the DMD shows for one LUT entry (bit-depth-wide field of its image)."""
        e = self.lut[lut_index]
        img = self.dmd_image(e.image_index)
        return ((img >> e.bit_position) & ((1 << e.bit_depth) - 1)).astype(np.uint8)

    def _close_timeline(self) -> None:
        self._timeline.extend(self._run_timeline(self.clock()))
        self._run_started_at = None

    def _run_timeline(self, until_ns: int) -> list[DisplayedPattern]:
        if self._run_started_at is None or self.lut_config is None:
            return []
        n, repeat = self.lut_config
        t = self._run_started_at
        out: list[DisplayedPattern] = []
        triggers = iter(sorted(x for x in self.trigger_times if x >= t))
        passes = 0
        while t < until_ns and (repeat == 0 or passes < repeat) and len(out) < 100_000:
            for k in range(n):
                e = self.lut[k]
                if e.wait_trigger:
                    t = next((x for x in triggers if x >= t), None)
                    if t is None or t >= until_ns:
                        return out
                if t >= until_ns:
                    return out
                out.append(DisplayedPattern(t, k, e.image_index, e.bit_position, e.bit_depth, e.exposure_us))
                t += (e.exposure_us + e.dark_us) * 1000
            passes += 1
        return out

    def displayed(self, until_ns: int | None = None) -> list[DisplayedPattern]:
        """The patterns shown so far (or until `until_ns`), with their start times: the current
        run's and, of finished runs, the newest ones `RecentLog` keeps."""
        until = self.clock() if until_ns is None else until_ns
        return self._timeline + (self._run_timeline(until) if self.sequencer == "running" else [])


# opcode -> (reader, writer, accepted write payload sizes)
_COMMANDS: dict[int, tuple] = {
    0x0100: (DLPC900Model._r_error, None, None),
    0x0101: (DLPC900Model._r_error_desc, None, None),
    0x0200: (DLPC900Model._r_power, DLPC900Model._w_power, {1}),
    0x0201: (DLPC900Model._r_idle, DLPC900Model._w_idle, {1}),
    0x0205: (DLPC900Model._r_version, None, None),
    0x0206: (DLPC900Model._r_hwconfig, None, None),
    0x0609: (DLPC900Model._r_park, DLPC900Model._w_park, {1}),
    0x1100: (DLPC900Model._r_curtain, DLPC900Model._w_curtain, {6}),
    0x1A00: (DLPC900Model._r_source, DLPC900Model._w_source, {1}),
    0x1A07: (DLPC900Model._r_led_enable, DLPC900Model._w_led_enable, {1}),
    0x1A0A: (DLPC900Model._r_hw_status, None, None),
    0x1A0B: (DLPC900Model._r_sys_status, None, None),
    0x1A0C: (DLPC900Model._r_main_status, None, None),
    0x1A1B: (DLPC900Model._r_display_mode, DLPC900Model._w_display_mode, {1}),
    0x1A1D: (lambda m: m._r_trig_out(1), lambda m, d: m._w_trig_out(1, d), {5}),
    0x1A1E: (lambda m: m._r_trig_out(2), lambda m, d: m._w_trig_out(2, d), {5}),
    0x1A24: (DLPC900Model._r_pattern, DLPC900Model._w_pattern, {1}),
    0x1A2A: (None, lambda m, d: m._w_image_init(False, d), {6}),
    0x1A2B: (None, lambda m, d: m._w_image_data(False, d), None),
    0x1A2C: (None, lambda m, d: m._w_image_init(True, d), {6}),
    0x1A2D: (None, lambda m, d: m._w_image_data(True, d), None),
    0x1A31: (DLPC900Model._r_lut_config, DLPC900Model._w_lut_config, {6}),
    0x1A34: (None, DLPC900Model._w_lut_define, {12}),
    0x1A35: (DLPC900Model._r_trig_in1, DLPC900Model._w_trig_in1, {2}),
    0x1A36: (DLPC900Model._r_trig_in2, DLPC900Model._w_trig_in2, {1}),
    0x0B01: (DLPC900Model._r_led_current, DLPC900Model._w_led_current, {3}),
}
