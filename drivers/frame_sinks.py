"""Frame sinks (`dpmhw.frame_sink.FrameSink`): where the loop's uint8 frames go.

Live frames reach a DLPC900 through its video input (HDMI / DisplayPort), so the projector sink
is a borderless full-screen window on the display the projector is attached to (`WindowSink`,
pygame-ce), presenting in step with that display's refresh. `FileSink` writes a PNG sequence or
a video for review; `RecordingSink` keeps frames in memory for tests. All three reject frames of
the wrong shape or dtype instead of resizing them, and carry the display's `DisplayTiming`.
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from dpmhw.display import DisplayTiming
from dpmhw.frame_sink import check_frame

Clock = Callable[[], int]


def _wait_until(t_target_ns: int, clock: Clock, sleep: Callable[[float], None]) -> None:
    """Sleep until `t_target_ns` if it is in the future (a late frame goes out at once)."""
    ahead = t_target_ns - clock()
    if ahead > 0:
        sleep(ahead / 1e9)


@dataclass(frozen=True)
class PresentedFrame:
    frame: np.ndarray
    t_target_ns: int
    presented_at_ns: int


class RecordingSink:
    """Keeps a copy of every frame with its target and presentation times (for tests).

    With `pace=True` it behaves like a display: its refreshes lie on a grid `timing.period_ns`
    apart from the clock's reading at construction, and `present` waits (via `sleep`) for the
    first refresh at or after both now and the target and returns that refresh instant. Without
    `pace` it has no refresh, like a file: it returns at once, with the time it kept the frame.
    """

    def __init__(self, *, shape: tuple[int, int] | None = None, timing: DisplayTiming = DisplayTiming(),
                 clock: Clock = time.monotonic_ns, sleep: Callable[[float], None] = time.sleep, pace: bool = False,
                 max_frames: int | None = None):
        self.shape = shape
        self.timing = timing
        self.clock, self.sleep, self.pace = clock, sleep, pace
        self.max_frames = max_frames
        self.frames: list[PresentedFrame] = []
        self.closed = False
        self._phase_ns = clock()

    def present(self, frame: np.ndarray, t_target_ns: int) -> int:
        if self.closed:
            raise RuntimeError("RecordingSink: present() after close()")
        check_frame(frame, self.shape)
        if self.pace:
            at = self.timing.next_vsync(max(self.clock(), t_target_ns), self._phase_ns)
            _wait_until(at, self.clock, self.sleep)
        else:
            at = self.clock()
        self.frames.append(PresentedFrame(frame.copy(), t_target_ns, at))
        if self.max_frames is not None and len(self.frames) > self.max_frames:
            del self.frames[0]
        return at

    def vsync_phase_ns(self) -> int:
        return self._phase_ns

    def close(self) -> None:
        self.closed = True


class FileSink:
    """Writes frames for review: a PNG sequence into a directory, or a video file.

    `path` ending in .avi / .mp4 / .mkv makes a video at `fps` (OpenCV's writer; .avi uses
    MJPG); anything else is a directory that receives frame_000000.png, ... (lossless).
    A file has no refresh: `present` writes at once and returns the time it finished writing.
    """

    VIDEO_CODECS = {".avi": "MJPG", ".mp4": "mp4v", ".mkv": "MJPG"}

    def __init__(self, path: str | os.PathLike, *, fps: float = 60.0, timing: DisplayTiming = DisplayTiming(),
                 clock: Clock = time.monotonic_ns):
        import cv2  # a core dependency; imported here so the module loads fast

        self._cv2 = cv2
        self.timing = timing
        self._phase_ns = clock()
        self.path = Path(path)
        self.fps = fps
        self.clock = clock
        self.count = 0
        self._writer = None
        self._shape: tuple[int, int] | None = None
        self.is_video = self.path.suffix.lower() in self.VIDEO_CODECS
        if not self.is_video:
            self.path.mkdir(parents=True, exist_ok=True)
        elif not self.path.parent.exists():
            raise ValueError(f"{self.path}: directory {self.path.parent} does not exist")

    def present(self, frame: np.ndarray, t_target_ns: int) -> int:
        check_frame(frame, self._shape)
        self._shape = frame.shape[:2]
        bgr = np.ascontiguousarray(frame[..., ::-1])
        if self.is_video:
            if self._writer is None:
                fourcc = self._cv2.VideoWriter_fourcc(*self.VIDEO_CODECS[self.path.suffix.lower()])
                h, w = self._shape
                self._writer = self._cv2.VideoWriter(str(self.path), fourcc, self.fps, (w, h))
                if not self._writer.isOpened():
                    raise OSError(f"{self.path}: OpenCV cannot open a video writer for this format")
            self._writer.write(bgr)
        else:
            name = self.path / f"frame_{self.count:06d}.png"
            if not self._cv2.imwrite(str(name), bgr):
                raise OSError(f"{name}: could not write PNG")
        self.count += 1
        return self.clock()

    def vsync_phase_ns(self) -> int:
        return self._phase_ns

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None


class WindowSink:
    """Borderless full-screen window on display `display`, fed to the projector's video input.

    Uses pygame-ce (a core dependency: the default sink). The window is always full-screen at the
    display's current mode, which must be the projector's native resolution: `size` is the
    session's output size, and a display of another size is refused here, at start (a frame
    of the wrong size would cover a corner of the projector's image). Nothing is scaled.

    Presents go out in step with the display's refresh. Where the platform gives vsync
    (pygame-ce's `set_mode(..., vsync=1)`, which needs SCALED or OPENGL), a flip blocks until the
    next refresh. At start the sink flips `VSYNC_PROBE_FLIPS` black frames, sleeping 0.3 and 1.3
    periods in turn between them, and is vsync-locked only if every flip returned on one grid of
    `timing.period_ns` (within `VSYNC_TOLERANCE`): a flip throttled to one period after the last
    (Mesa's software swap on Xvfb) returns at once after the longer sleep and fails that. Locked,
    `present` sleeps until half a period before the refresh it aims at, flips, and returns the
    flip's return time, which re-locks the phase. Otherwise the sink keeps a software refresh
    grid at `timing.refresh_hz` from its start: `present` waits for the first grid instant at or
    after the target, flips, and returns that instant. `vsync_locked` says which.

    What a real display adds, and this sink cannot see: the flip's return lags the refresh by
    the wake-up of this thread (tens of microseconds to a millisecond), a compositor or driver
    that queues frames shows each one or more refreshes later, the GPU's scan-out clock drifts
    from `refresh_hz` (the phase re-lock follows it; the software grid does not), and the
    projector adds its own delay after the scan-out (`timing.controller_delay_ns`).
    """

    VSYNC_PROBE_FLIPS = 8
    VSYNC_TOLERANCE = 0.1  # fraction of a period a probed flip may lie off the grid

    def __init__(self, display: int = 0, *, size: tuple[int, int] | None = None,
                 timing: DisplayTiming = DisplayTiming(), clock: Clock = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep, title: str = "dpmhw projector"):
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame

        self._pg = pygame
        self.timing = timing
        self.clock, self.sleep = clock, sleep
        pygame.display.init()
        try:
            w, h = _display_size(pygame, display, size)
        except ValueError:
            pygame.display.quit()
            raise
        flags = pygame.NOFRAME | pygame.FULLSCREEN
        pygame.display.set_caption(title)
        self.shape = (h, w)
        self.closed = False
        self._phase_ns = clock()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # "no fast renderer available": no vsync either
                self._surface = pygame.display.set_mode((w, h), flags | pygame.SCALED, display=display, vsync=1)
            self.vsync_locked = self._probe_vsync()
        except (pygame.error, Warning):  # no vsync on this platform
            self.vsync_locked = False
        if not self.vsync_locked:  # a plain window whose flips never block, paced by the software grid
            self._surface = pygame.display.set_mode((w, h), flags, display=display)
        pygame.mouse.set_visible(False)

    def _probe_vsync(self) -> bool:
        """Flip black frames at uneven gaps; vsync-locked when every flip returns on one refresh grid."""
        self._blit(np.zeros((*self.shape, 3), np.uint8))
        p = self.timing.period_ns
        returns = []
        for k in range(self.VSYNC_PROBE_FLIPS):
            self._pg.display.flip()
            returns.append(self.clock())
            self.sleep((0.3 if k % 2 else 1.3) * p / 1e9)
        self._phase_ns = returns[-1]
        off = (np.asarray(returns[1:]) - returns[0]) / p  # the first flip may land mid-period
        return bool((np.abs(off - np.round(off)) <= self.VSYNC_TOLERANCE).all() and (np.diff(np.round(off)) >= 1).all())

    def _blit(self, frame: np.ndarray) -> None:
        image = self._pg.image.frombuffer(np.ascontiguousarray(frame), (self.shape[1], self.shape[0]), "RGB")  # no copy
        self._surface.blit(image, (0, 0))

    def present(self, frame: np.ndarray, t_target_ns: int) -> int:
        if self.closed:
            raise RuntimeError("WindowSink: present() after close()")
        check_frame(frame, self.shape)
        vsync = self.timing.next_vsync(max(self.clock(), t_target_ns), self._phase_ns)
        if self.vsync_locked:
            _wait_until(vsync - self.timing.period_ns // 2, self.clock, self.sleep)
        else:
            _wait_until(vsync, self.clock, self.sleep)
        self._blit(frame)
        self._pg.display.flip()
        self._pg.event.pump()  # keep the window responsive to the window manager
        if not self.vsync_locked:
            return vsync
        self._phase_ns = self.clock()  # the flip returned at the refresh that scans the frame out
        return self._phase_ns

    def snapshot(self) -> np.ndarray:
        """(H, W, 3) uint8 of what the window holds now (for tests and diagnostics)."""
        return self._pg.surfarray.array3d(self._surface).swapaxes(0, 1).copy()

    def vsync_phase_ns(self) -> int:
        return self._phase_ns

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._pg.display.quit()


def _display_size(pygame, display: int, size: tuple[int, int] | None) -> tuple[int, int]:
    """Display `display`'s current mode, which must be `size` when given (ValueError otherwise)."""
    n = pygame.display.get_num_displays()
    if not 0 <= display < n:
        raise ValueError(f"display: {display} does not exist ({n} display(s) attached)")
    native = tuple(pygame.display.get_desktop_sizes()[display])
    if size is not None and tuple(size) != native:
        raise ValueError(f"display {display} runs at {native[0]}×{native[1]}, but the session outputs {size[0]}×{size[1]} "
                         "(set the display to the projector's native mode, or render.width/height to match)")
    return native


def check_display(display: int, size: tuple[int, int] | None = None) -> None:
    """`WindowSink`'s checks of the display, without opening a window (a config check)."""
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import pygame

    pygame.display.init()
    try:
        _display_size(pygame, display, size)
    finally:
        pygame.display.quit()


def make_sink(kind: str, **kwargs):
    """Sink by name, for configs: "window", "file" or "recording"."""
    kinds = {"window": WindowSink, "file": FileSink, "recording": RecordingSink}
    if kind not in kinds:
        raise ValueError(f"frame sink: expected one of {sorted(kinds)}, got {kind!r}")
    return kinds[kind](**kwargs)
