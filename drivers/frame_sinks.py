"""Frame sinks (`dpmhw.frame_sink.FrameSink`): where the loop's uint8 frames go.

Live frames reach a DLPC900 through its video input (HDMI / DisplayPort), so the projector sink
is a borderless full-screen window on the display the projector is attached to (`WindowSink`,
pygame-ce). `FileSink` writes a PNG sequence or a video for
review; `RecordingSink` keeps frames in memory for tests. All three reject frames of the wrong
shape or dtype instead of resizing them.
"""

from __future__ import annotations

import os
import time
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

    With `pace=True` it waits for each target time like a display would (via `sleep`).
    """

    timing = DisplayTiming()  # no refresh model yet: frames go out when presented

    def __init__(self, *, shape: tuple[int, int] | None = None, clock: Clock = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep, pace: bool = False, max_frames: int | None = None):
        self.shape = shape
        self.clock, self.sleep, self.pace = clock, sleep, pace
        self.max_frames = max_frames
        self.frames: list[PresentedFrame] = []
        self.closed = False

    def present(self, frame: np.ndarray, t_target_ns: int) -> int:
        if self.closed:
            raise RuntimeError("RecordingSink: present() after close()")
        check_frame(frame, self.shape)
        if self.pace:
            _wait_until(t_target_ns, self.clock, self.sleep)
        now = self.clock()
        self.frames.append(PresentedFrame(frame.copy(), t_target_ns, now))
        if self.max_frames is not None and len(self.frames) > self.max_frames:
            del self.frames[0]
        return now

    def vsync_phase_ns(self) -> int:
        return 0

    def close(self) -> None:
        self.closed = True


class FileSink:
    """Writes frames for review: a PNG sequence into a directory, or a video file.

    `path` ending in .avi / .mp4 / .mkv makes a video at `fps` (OpenCV's writer; .avi uses
    MJPG); anything else is a directory that receives frame_000000.png, ... (lossless).
    """

    VIDEO_CODECS = {".avi": "MJPG", ".mp4": "mp4v", ".mkv": "MJPG"}

    timing = DisplayTiming()  # no refresh model yet: frames go out when presented

    def __init__(self, path: str | os.PathLike, *, fps: float = 60.0, clock: Clock = time.monotonic_ns):
        import cv2  # a core dependency; imported here so the module loads fast

        self._cv2 = cv2
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
        return 0

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
    `present` waits for the target time, blits and flips, and returns the time the flip returned.
    """

    timing = DisplayTiming()  # no refresh model yet: frames go out when presented

    def __init__(self, display: int = 0, *, size: tuple[int, int] | None = None, clock: Clock = time.monotonic_ns,
                 sleep: Callable[[float], None] = time.sleep, title: str = "dpmhw projector"):
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        import pygame

        self._pg = pygame
        self.clock, self.sleep = clock, sleep
        pygame.display.init()
        try:
            w, h = _display_size(pygame, display, size)
        except ValueError:
            pygame.display.quit()
            raise
        flags = pygame.NOFRAME | pygame.FULLSCREEN
        pygame.display.set_caption(title)
        self._surface = pygame.display.set_mode((w, h), flags, display=display)
        pygame.mouse.set_visible(False)
        self.shape = (self._surface.get_height(), self._surface.get_width())
        self.closed = False

    def present(self, frame: np.ndarray, t_target_ns: int) -> int:
        if self.closed:
            raise RuntimeError("WindowSink: present() after close()")
        check_frame(frame, self.shape)
        pg = self._pg
        image = pg.image.frombuffer(np.ascontiguousarray(frame).tobytes(), (self.shape[1], self.shape[0]), "RGB")
        _wait_until(t_target_ns, self.clock, self.sleep)
        self._surface.blit(image, (0, 0))
        pg.display.flip()
        pg.event.pump()  # keep the window responsive to the window manager
        return self.clock()

    def snapshot(self) -> np.ndarray:
        """(H, W, 3) uint8 of what the window holds now (for tests and diagnostics)."""
        return self._pg.surfarray.array3d(self._surface).swapaxes(0, 1).copy()

    def vsync_phase_ns(self) -> int:
        return 0

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
