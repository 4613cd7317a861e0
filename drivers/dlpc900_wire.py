"""DLPC900 USB-HID framing (host side): opcodes, request reports, reply headers, typed errors.

A request is one message: flags (bit 7 read, bit 6 reply wanted, bits 2:0 destination 0),
sequence byte, little-endian length (= 2 + data bytes), little-endian opcode (CMD3 low byte
first, then CMD2), data. It travels as 64-byte reports: the first carries the header, the rest
continue the message raw. A reply echoes flags (bit 5 = error) and sequence, then a
little-endian data length and the data, split the same way. pyusb sees no HID report id.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from dpmhw.errors import DpmhwError

REPORT = 64
HEADER = 4
CMD_BUFFER = 512
IMAGE_CHUNK = 504  # image bytes per 0x1A2B message: 4 header + 2 opcode + 2 count + 504 = 512

FLAG_READ = 0x80
FLAG_REPLY = 0x40
FLAG_ERROR = 0x20


class Cmd(IntEnum):
    ERROR_CODE = 0x0100
    ERROR_DESCRIPTION = 0x0101
    POWER_MODE = 0x0200
    IDLE_MODE = 0x0201
    FIRMWARE_VERSION = 0x0205
    HARDWARE_CONFIG = 0x0206
    PARK = 0x0609
    CURTAIN_COLOR = 0x1100
    INPUT_SOURCE = 0x1A00
    LED_ENABLE = 0x1A07
    HARDWARE_STATUS = 0x1A0A
    SYSTEM_STATUS = 0x1A0B
    MAIN_STATUS = 0x1A0C
    DISPLAY_MODE = 0x1A1B
    TRIGGER_OUT1 = 0x1A1D
    TRIGGER_OUT2 = 0x1A1E
    PATTERN_START_STOP = 0x1A24
    IMAGE_LOAD_INIT = 0x1A2A
    IMAGE_DATA = 0x1A2B
    IMAGE_LOAD_INIT_SECONDARY = 0x1A2C
    IMAGE_DATA_SECONDARY = 0x1A2D
    LUT_CONFIGURE = 0x1A31
    LUT_DEFINITION = 0x1A34
    TRIGGER_IN1 = 0x1A35
    TRIGGER_IN2 = 0x1A36
    LED_CURRENT = 0x0B01


# Reply data length of every read, so a reply of another length is caught as malformed.
READ_LENGTH: dict[int, int | tuple[int, int]] = {
    Cmd.ERROR_CODE: 1, Cmd.ERROR_DESCRIPTION: (1, 128), Cmd.POWER_MODE: 1, Cmd.IDLE_MODE: 1,
    Cmd.FIRMWARE_VERSION: 16, Cmd.HARDWARE_CONFIG: 32, Cmd.PARK: 1, Cmd.CURTAIN_COLOR: 6,
    Cmd.INPUT_SOURCE: 1, Cmd.LED_ENABLE: 1, Cmd.HARDWARE_STATUS: 1, Cmd.SYSTEM_STATUS: 1,
    Cmd.MAIN_STATUS: 1, Cmd.DISPLAY_MODE: 1, Cmd.TRIGGER_OUT1: 5, Cmd.TRIGGER_OUT2: 5,
    Cmd.PATTERN_START_STOP: 1, Cmd.LUT_CONFIGURE: 6, Cmd.TRIGGER_IN1: 2, Cmd.TRIGGER_IN2: 1,
    Cmd.LED_CURRENT: 3,
}

ERROR_CODES = {
    0: "no error", 1: "batch file checksum error", 2: "device failure", 3: "invalid command",
    4: "incompatible controller or DMD", 5: "command not allowed in current mode", 6: "invalid command parameter",
    7: "item referred by the parameter is not present", 8: "out of memory", 9: "invalid BMP compression type",
    10: "pattern bit number out of range", 11: "pattern BMP not present in flash", 12: "pattern dark time out of range",
    13: "signal delay parameter out of range", 14: "pattern exposure time out of range",
    15: "pattern number out of range", 16: "invalid pattern definition", 17: "pattern image memory address out of range",
    255: "internal error",
}


# ---- errors -------------------------------------------------------------------------------
class DLPC900Error(DpmhwError):
    """Base of every error the DLPC900 driver raises."""


class DLPC900NotFound(DLPC900Error, LookupError):
    """No matching controller on the bus (or several and no serial number to choose)."""


class DLPC900Timeout(DLPC900Error, TimeoutError):
    """The controller did not answer within the read timeout."""


class DLPC900USBError(DLPC900Error, OSError):
    """The USB transfer itself failed (stall, I/O error, permissions); `errno` as libusb gave it."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno


class DLPC900Disconnected(DLPC900USBError):
    """The device went away (errno 19, ENODEV); `DLPC900.reconnect()` can bring it back."""


class DLPC900ProtocolError(DLPC900Error):
    """A reply that does not follow the framing: short, wrong sequence or wrong length."""


class DLPC900DeviceError(DLPC900Error):
    """The controller rejected a command; `code` and `description` come from 0x0100 / 0x0101
    (an empty description is replaced by the code's name)."""

    def __init__(self, command: int, code: int, description: str):
        name = ERROR_CODES.get(code, "unknown error")
        self.command = command
        self.code = code
        self.description = description or name
        super().__init__(f"DLPC900 rejected command 0x{command:04X}: error {code} ({name}): {self.description}")


def c_string(data: bytes) -> str:
    """The text of a NUL-terminated ASCII field (error description, hardware tag)."""
    return data.split(b"\x00", 1)[0].decode("ascii", "replace")


class DLPC900SafetyError(DLPC900Error):
    """A safe state (dark, sequencer stopped) could not be confirmed by read-back."""


# ---- framing ------------------------------------------------------------------------------
def request_reports(seq: int, cmd: int, data: bytes = b"", *, read: bool = False, reply: bool = True) -> list[bytes]:
    """The 64-byte OUT reports that carry one command."""
    if not 0 <= seq <= 0xFF:
        raise ValueError(f"seq: expected 0..255, got {seq}")
    length = 2 + len(data)
    if HEADER + length > CMD_BUFFER:
        raise ValueError(f"command 0x{cmd:04X}: {len(data)} data bytes exceed the 512-byte command buffer")
    flags = (FLAG_READ if read else 0) | (FLAG_REPLY if (reply or read) else 0)
    msg = bytes([flags, seq]) + struct.pack("<HH", length, cmd) + bytes(data)
    return [msg[i:i + REPORT].ljust(REPORT, b"\x00") for i in range(0, len(msg), REPORT)]


@dataclass(frozen=True)
class ReplyHeader:
    flags: int
    seq: int
    length: int

    @property
    def error(self) -> bool:
        return bool(self.flags & FLAG_ERROR)


def parse_reply_header(report: bytes) -> ReplyHeader:
    if len(report) < HEADER:
        raise DLPC900ProtocolError(f"reply of {len(report)} bytes is shorter than the 4-byte header")
    return ReplyHeader(report[0], report[1], report[2] | (report[3] << 8))
