"""When a presented frame becomes light: the display's timing model.

A frame handed to the projector's video input is scanned out at the link's next refresh (vsync),
and the controller lights the mirrors `controller_delay_ns` after that scan-out starts. What it
lights then depends on the display mode:

- ``video``: the whole 24-bit frame for one refresh period (one photon window);
- ``pattern-8bit`` (the DLPC900's video-pattern mode): the frame's R, G and B bit planes as three
  8-bit monochrome sub-frames, one after another, each filling a third of the period (180 Hz at a
  60 Hz link) and lit by the LED its pattern entry names. A colour scene runs field-sequential:
  sub-frame k shows colour channel k under LED k.

Everything here is relative to the scan-out instant (`vsync_ns`) of the video frame that carries
the picture, on the host's monotonic clock. Prediction targets the middle of each photon window;
the registration of a sub-frame is measured there.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

__all__ = ["DISPLAY_MODES", "DisplayTiming", "PhotonWindow"]

DISPLAY_MODES = ("video", "pattern-8bit")

_LEDS = ((True, False, False), (False, True, False), (False, False, True))


@dataclass(frozen=True)
class PhotonWindow:
    """One (sub-)frame's light, relative to its video frame's scan-out."""

    channel: int | None  # the RGB channel shown (0, 1, 2); None: all three at once (video mode)
    start_ns: int  # first photon after the scan-out starts
    duration_ns: int
    leds: tuple[bool, bool, bool]  # which LEDs light it (red, green, blue)

    @property
    def mid_ns(self) -> int:
        return self.start_ns + self.duration_ns // 2


@dataclass(frozen=True)
class DisplayTiming:
    """The link's refresh, the controller's delay and the mode's photon windows."""

    mode: str = "video"
    refresh_hz: float = 60.0
    controller_delay_ns: int = 0

    def __post_init__(self) -> None:
        if self.mode not in DISPLAY_MODES:
            raise ValueError(f"display.mode: expected one of {', '.join(DISPLAY_MODES)}, got {self.mode!r}")
        if not 1.0 <= self.refresh_hz <= 1000.0:
            raise ValueError(f"display.refresh_hz: expected 1 to 1000, got {self.refresh_hz!r}")
        if not 0 <= self.controller_delay_ns <= 1_000_000_000:
            raise ValueError(f"display.controller_delay_ms: expected 0 to 1000 ms, got {self.controller_delay_ns / 1e6!r}")

    @cached_property  # read several times at every refresh by the present thread
    def period_ns(self) -> int:
        return round(1e9 / self.refresh_hz)

    @cached_property
    def windows(self) -> tuple[PhotonWindow, ...]:
        """The photon windows of one video frame, in the order they are lit."""
        p, d = self.period_ns, self.controller_delay_ns
        if self.mode == "video":
            return (PhotonWindow(None, d, p, (True, True, True)),)
        third = p // 3
        return tuple(PhotonWindow(k, d + k * third, third, _LEDS[k]) for k in range(3))

    def photon_mid_ns(self, vsync_ns: int) -> list[int]:
        """The middle of each photon window of the frame scanned out at `vsync_ns`."""
        return [vsync_ns + w.mid_ns for w in self.windows]

    def next_vsync(self, t_ns: int, phase_ns: int) -> int:
        """The first refresh at or after `t_ns`, given one known refresh instant `phase_ns`."""
        p = self.period_ns
        return phase_ns + -(-(t_ns - phase_ns) // p) * p
