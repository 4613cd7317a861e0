"""Where finished frames go: the one interface the loop knows about the projector's video input.

The loop calls `present` once per frame; implementations live in `drivers/` (a full-screen
window on the projector's display, a PNG/video file writer, an in-memory recorder for tests).
`dpmhw` never imports them: a session factory picks one by name.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from dpmhw.display import DisplayTiming


@runtime_checkable
class FrameSink(Protocol):
    """Consumer of output frames.

    `present(frame, t_target_ns)` shows `frame`, a (H, W, 3) uint8 sRGB image with row 0 at
    the top, at the first refresh at or after `t_target_ns` (monotonic clock) and returns
    that refresh's scan-out instant (ns): the frame's light follows as `timing` says. A sink
    without a refresh (a file writer) returns when it wrote the frame. A sink never silently
    drops or resizes a frame: a wrong shape or dtype raises `ValueError`.

    `timing` is the display's model; `vsync_phase_ns()` one refresh instant it has seen or
    keeps (the refreshes are `timing.period_ns` apart from there).
    """

    timing: DisplayTiming

    def present(self, frame: np.ndarray, t_target_ns: int) -> int: ...

    def vsync_phase_ns(self) -> int: ...

    def close(self) -> None: ...


def check_frame(frame: np.ndarray, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Validate an output frame; `shape` is the expected (H, W) or None for any size.

    Shared by every sink so that all of them reject the same bad input with the same message.
    """
    if not isinstance(frame, np.ndarray):
        raise ValueError(f"frame: expected a numpy array, got {type(frame).__name__}")
    if frame.dtype != np.uint8:
        raise ValueError(f"frame: expected dtype uint8, got {frame.dtype}")
    if frame.ndim != 3 or frame.shape[2] != 3:
        raise ValueError(f"frame: expected shape (H, W, 3), got {frame.shape}")
    if shape is not None and frame.shape[:2] != tuple(shape):
        raise ValueError(f"frame: expected (H, W) = {tuple(shape)}, got {frame.shape[:2]}")
    return frame
