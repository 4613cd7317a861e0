"""The device side of the video cable and the DLPC900's video input: what a `--mock` session
presents to, and what the projector makes of each frame, with the times its light falls.

`VideoLink` is a `dpmhw.frame_sink.FrameSink`. The link refreshes on a grid `timing.period_ns`
apart (from `phase_ns`, by default the clock's reading at construction). `present` latches the
frame for the first refresh at or after both now and its target and, like a vsync'd swap, waits
for that refresh (`block=False`: returns at once, a mailbox swap). A frame replaced by another
before its refresh came is never scanned out and is counted in `never_shown`; a refresh with no
new frame scans the last one out again (`repeats`), as a GPU does.

Each scanned-out frame is decoded as the controller would, from the `DLPC900Model` the USB
emulator serves (the same instance), at its scan-out instant `v`:

- dark (standby, idle, parked, LEDs off), or a pattern mode that does not read the video input
  (pre-stored, on-the-fly), or video pattern mode with the sequencer not running: no light;
- video mode: one exposure of the RGB frame, `[v + delay, v + delay + period)`, all LEDs;
- video pattern mode: the run of LUT entries this frame shows (from an entry that waits for the
  VSYNC to the next; `video_frame_groups`), one after another from `v + delay`: each entry
  exposes `exposure_us` then stays dark `dark_us`, shows bits `bit_position …
  bit_position + bit_depth − 1` of the 24-bit input word and lights the LEDs its colour names.
  The word's bits 0–7 are the green channel, 8–15 red and 16–23 blue, the order TI's
  controllers number a video frame's bit planes (DLPC350 guide's pattern number mapping; public
  DLPC900 video-pattern hosts extract the planes the same way). A LUT whose repeat count is not
  0 (forever) stops after that many patterns.

`delay` is the controller's own delay from scan-out to first photon (`controller_delay_ns`,
by default `timing.controller_delay_ns`); it is the emulated device's, so a test can give the
host's timing model a different one and see the error.

Every exposure is a row in `exposures` (bounded: the newest `max_rows`); with `keep_images`
the newest that many rows also carry the decoded (H, W) image (uint8 for ≤ 8 bits). The link
never imports `drivers`.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from dpmhw.display import DisplayTiming
from dpmhw.frame_sink import check_frame
from firmware_mocks.dlpc900_model import DLPC900Model, video_frame_groups

__all__ = ["Exposure", "VideoLink", "CHANNEL_OF_BIT", "input_word"]

_SHIFT = (8, 0, 16)  # per RGB channel of the frame (R, G, B): where its 8 bits sit in the 24-bit word
CHANNEL_OF_BIT = {bit: channel for channel, bit in enumerate(_SHIFT)}


def input_word(frame: np.ndarray) -> np.ndarray:
    """(H, W) uint32 24-bit words of an RGB frame as the video-pattern sequencer numbers them."""
    f = frame.astype(np.uint32)
    return (f[..., 0] << _SHIFT[0]) | (f[..., 1] << _SHIFT[1]) | (f[..., 2] << _SHIFT[2])


@dataclass(frozen=True)
class Exposure:
    """One (sub-)frame of light the projector showed."""

    frame: int  # video frame number: the n-th frame presented to the link (0-based)
    scanout_ns: int  # the refresh at which the frame was scanned out
    lut_index: int | None  # the LUT entry (video pattern mode); None in video mode
    channel: int | None  # the RGB channel shown when the entry is one whole channel; None otherwise
    bit_position: int  # lowest bit of the input word shown (video mode: 0)
    bit_depth: int  # video mode: 24
    leds: tuple[bool, bool, bool]  # red, green, blue
    t_start_ns: int
    t_end_ns: int
    repeat: bool  # the frame scanned out again for want of a new one
    image: np.ndarray | None = None  # the decoded image (with keep_images)


class VideoLink:
    """Emulated video link + DLPC900 video input (see the module docstring)."""

    def __init__(self, model: DLPC900Model, *, timing: DisplayTiming = DisplayTiming(),
                 controller_delay_ns: int | None = None, shape: tuple[int, int] | None = None,
                 clock: Callable[[], int] = time.monotonic_ns, sleep: Callable[[float], None] = time.sleep,
                 phase_ns: int | None = None, block: bool = True, max_rows: int = 4096, keep_images: int = 0):
        if max_rows < 1 or not 0 <= keep_images <= max_rows:
            raise ValueError(f"max_rows ≥ 1 and 0 ≤ keep_images ≤ max_rows, got {max_rows}, {keep_images}")
        self.model, self.timing, self.shape = model, timing, shape
        self.delay_ns = timing.controller_delay_ns if controller_delay_ns is None else controller_delay_ns
        if self.delay_ns < 0:
            raise ValueError(f"controller_delay_ns: expected ≥ 0, got {self.delay_ns}")
        self.clock, self.sleep, self.block = clock, sleep, block
        self._phase_ns = clock() if phase_ns is None else phase_ns
        self.keep_images = keep_images
        self.exposures: deque[Exposure] = deque(maxlen=max_rows)
        self.frames_presented = 0
        self.frames_shown = 0
        self.never_shown = 0
        self.repeats = 0
        self._pending: tuple[int, int, np.ndarray] | None = None  # (frame number, refresh, frame)
        self._last: tuple[int, np.ndarray] | None = None  # the frame the link scans out now
        self._scanned_ns = self._newest_refresh(clock())  # the last refresh processed
        self._group = 0  # the LUT's next frame group
        self._patterns_shown = 0  # since the sequencer started (for a LUT repeat count)
        self._run_started: int | None = None
        self._lock = threading.Lock()
        self.closed = False
        model.video_period_ns = timing.period_ns  # the cable is in: the input locks to its syncs

    # ---- FrameSink -------------------------------------------------------------------------
    def present(self, frame: np.ndarray, t_target_ns: int) -> int:
        if self.closed:
            raise RuntimeError("VideoLink: present() after close()")
        check_frame(frame, self.shape)
        with self._lock:
            now = self.clock()
            self._advance(now)
            v = self.timing.next_vsync(max(now, t_target_ns), self._phase_ns)
            if v <= self._scanned_ns:  # that refresh is scanning out already: the next one
                v += self.timing.period_ns
            if self._pending is not None:
                self.never_shown += 1  # replaced before its refresh came
            self._pending = (self.frames_presented, v, frame.copy())
            self.frames_presented += 1
        if self.block:
            ahead = v - self.clock()
            if ahead > 0:
                self.sleep(ahead / 1e9)
            self.poll()
        return v

    def vsync_phase_ns(self) -> int:
        return self._phase_ns

    def close(self) -> None:
        if not self.closed:
            self.poll()
            self.closed = True
            self.model.video_period_ns = None  # cable out: the input loses sync

    # ---- the device side -----------------------------------------------------------------
    def poll(self) -> None:
        """Scan out every refresh up to now (tests call it after moving a fake clock)."""
        with self._lock:
            self._advance(self.clock())

    def _advance(self, now: int) -> None:
        """Process the refreshes in (last processed, now]: the pending frame at its refresh,
        the last frame again at the others."""
        p = self.timing.period_ns
        last_v = self._newest_refresh(now)
        while self._scanned_ns < last_v:
            if self._pending is not None and self._pending[1] <= last_v:
                due = self._pending[1]
                self._repeat(self._scanned_ns + p, due - p)
                number, v, frame = self._pending
                self._pending = None
                self._last = (number, frame)
                self.frames_shown += 1
                self._scan_out(number, v, frame, repeat=False)
                self._scanned_ns = v
            else:
                self._repeat(self._scanned_ns + p, last_v)
                self._scanned_ns = last_v

    def _newest_refresh(self, t: int) -> int:
        return self.timing.next_vsync(t + 1, self._phase_ns) - self.timing.period_ns

    def _repeat(self, first_v: int, last_v: int) -> None:
        """The last frame scanned out again at the refreshes first_v … last_v (the newest
        `max_rows` of them decoded; a long idle gap is counted, not replayed)."""
        if self._last is None or last_v < first_v:
            return
        p = self.timing.period_ns
        n = (last_v - first_v) // p + 1
        self.repeats += n
        keep = min(n, self.exposures.maxlen)
        number, frame = self._last
        for k in range(n - keep, n):
            self._scan_out(number, first_v + k * p, frame, repeat=True)

    def _scan_out(self, number: int, v: int, frame: np.ndarray, *, repeat: bool) -> None:
        m = self.model
        t = v + self.delay_ns
        if m.dark_at(t):
            return
        mode = m.settled_display_mode
        if mode == 0:
            self._row(number, v, None, 0, 24, (True, True, True), t, t + self.timing.period_ns, repeat,
                      lambda: frame.copy())
            return
        if mode != 2 or m.sequencer != "running" or m.lut_config is None:
            self._run_started = None
            return
        n, repeat_count = m.lut_config
        if self._run_started is None or m.run_started_ns != self._run_started:  # a new run: from entry 0
            self._run_started, self._patterns_shown, self._group = m.run_started_ns, 0, 0
        groups = video_frame_groups([m.lut[k] for k in range(n)])
        group = groups[self._group % len(groups)]
        self._group += 1
        word = None
        for e in group:
            if repeat_count and self._patterns_shown >= repeat_count:
                return
            self._patterns_shown += 1
            leds = (bool(e.color & 1), bool(e.color & 2), bool(e.color & 4))
            end = t + e.exposure_us * 1000
            if self.keep_images:
                word = input_word(frame) if word is None else word
            self._row(number, v, e.index, e.bit_position, e.bit_depth, leds, t, end, repeat,
                      lambda e=e, w=word: ((w >> e.bit_position) & ((1 << e.bit_depth) - 1)).astype(np.uint8))
            t = end + e.dark_us * 1000

    def _row(self, number, v, lut_index, bit_position, bit_depth, leds, t0, t1, repeat, image) -> None:
        channel = CHANNEL_OF_BIT.get(bit_position) if bit_depth == 8 else None
        rows = self.exposures
        rows.append(Exposure(number, v, lut_index, channel, bit_position, bit_depth, leds, t0, t1, repeat,
                             image() if self.keep_images else None))
        if 0 < self.keep_images < len(rows):  # only the newest `keep_images` rows hold an image
            rows[-1 - self.keep_images] = dataclasses.replace(rows[-1 - self.keep_images], image=None)
