"""What the DLPC900 reports and takes, as typed values: modes, versions, status flags, timings.

Status bytes are decoded into named flags with bit 0 the least significant bit, as the
programmer's guide numbers them. Kept apart from `drivers/dlpc900.py` so the CLI, the server
and tests can use the types without the USB stack.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Sequence

# Minimum exposure per bit depth (DLP6500). 1, 2, 4, 8 bits: protocols.md; 3, 5, 6, 7 bits:
# the DLPC900 datasheet's pattern-rate table. Checked before anything is sent.
MIN_EXPOSURE_US = {1: 105, 2: 304, 3: 394, 4: 823, 5: 1215, 6: 1487, 7: 1998, 8: 4046}
MAX_U24 = (1 << 24) - 1


class DisplayMode(IntEnum):
    VIDEO = 0
    PRE_STORED_PATTERN = 1
    VIDEO_PATTERN = 2
    PATTERN_ON_THE_FLY = 3


class Color(IntEnum):
    """LED colour of a pattern (LUT definition bits 6:4)."""

    NONE = 0
    RED = 1
    GREEN = 2
    YELLOW = 3
    BLUE = 4
    MAGENTA = 5
    CYAN = 6
    WHITE = 7


DMD_NAMES = {1: "DLP6500", 2: "DLP9000", 3: "DLP670S", 4: "DLP500YX"}


@dataclass(frozen=True)
class Version:
    major: int
    minor: int
    patch: int

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.patch}"


@dataclass(frozen=True)
class FirmwareVersion:
    application: Version
    api: Version
    software_config: Version
    sequencer_config: Version

    @classmethod
    def decode(cls, data: bytes) -> "FirmwareVersion":
        parts = [Version(ma, mi, p) for p, mi, ma in struct.iter_unpack("<HBB", data)]
        return cls(*parts)


@dataclass(frozen=True)
class HardwareConfig:
    dmd: int  # 1 DLP6500, 2 DLP9000, 3 DLP670S, 4 DLP500YX
    tag: str

    @property
    def dmd_name(self) -> str:
        return DMD_NAMES.get(self.dmd, f"unknown DMD ({self.dmd})")


def _flags(value: int, names: Sequence[str | None]) -> dict[str, bool]:
    return {name: bool(value >> bit & 1) for bit, name in enumerate(names) if name}


@dataclass(frozen=True)
class HardwareStatus:
    raw: int
    init_ok: bool
    incompatible_controller_dmd: bool
    dmd_reset_controller_error: bool
    forced_swap_error: bool
    secondary_controller_present: bool
    sequencer_abort: bool
    sequencer_error: bool

    @classmethod
    def decode(cls, v: int) -> "HardwareStatus":
        return cls(v, **_flags(v, ["init_ok", "incompatible_controller_dmd", "dmd_reset_controller_error",
                                   "forced_swap_error", "secondary_controller_present", None,
                                   "sequencer_abort", "sequencer_error"]))

    @property
    def faults(self) -> list[str]:
        names = ["incompatible_controller_dmd", "dmd_reset_controller_error", "forced_swap_error",
                 "sequencer_abort", "sequencer_error"]
        return [n for n in names if getattr(self, n)] + ([] if self.init_ok else ["init_not_ok"])


@dataclass(frozen=True)
class SystemStatus:
    raw: int
    memory_test_passed: bool

    @classmethod
    def decode(cls, v: int) -> "SystemStatus":
        return cls(v, bool(v & 1))


@dataclass(frozen=True)
class MainStatus:
    raw: int
    dmd_parked: bool
    sequencer_running: bool
    video_frozen: bool
    external_source_locked: bool
    port1_syncs_valid: bool
    port2_syncs_valid: bool

    @classmethod
    def decode(cls, v: int) -> "MainStatus":
        return cls(v, **_flags(v, ["dmd_parked", "sequencer_running", "video_frozen", "external_source_locked",
                                   "port1_syncs_valid", "port2_syncs_valid"]))


@dataclass(frozen=True)
class TriggerOut:
    invert: bool
    rising_delay_us: int
    falling_delay_us: int


@dataclass(frozen=True)
class LedEnable:
    red: bool
    green: bool
    blue: bool
    sequencer_controlled: bool

    def encode(self) -> int:
        return int(self.red) | int(self.green) << 1 | int(self.blue) << 2 | int(self.sequencer_controlled) << 3

    @classmethod
    def decode(cls, v: int) -> "LedEnable":
        return cls(bool(v & 1), bool(v & 2), bool(v & 4), bool(v & 8))


@dataclass(frozen=True)
class PatternTiming:
    """How each pattern of a sequence is shown (one LUT definition per pattern)."""

    exposure_us: int
    dark_us: int = 0
    bit_depth: int = 1
    color: Color = Color.WHITE
    wait_for_trigger: bool = False
    clear_after: bool = False
    trigger_out2: bool = True

    def check(self) -> None:
        if self.bit_depth not in MIN_EXPOSURE_US:
            raise ValueError(f"bit_depth: expected 1..8, got {self.bit_depth}")
        low = MIN_EXPOSURE_US[self.bit_depth]
        if not low <= self.exposure_us <= MAX_U24:
            raise ValueError(f"exposure_us: {self.exposure_us} µs is outside {low}..{MAX_U24} µs, "
                             f"the range for {self.bit_depth}-bit patterns (DLP6500 minimum {low} µs)")
        if not 0 <= self.dark_us <= MAX_U24:
            raise ValueError(f"dark_us: expected 0..{MAX_U24}, got {self.dark_us}")


@dataclass(frozen=True)
class BlankReport:
    """How the projector was made dark and what the read-back showed."""

    method: str  # "idle", "leds off" or "standby"
    idle: bool | None
    sequencer_running: bool | None
    led_enable: int | None


@dataclass(frozen=True)
class DeviceInfo:
    serial: str | None
    bus: int | None
    address: int | None
