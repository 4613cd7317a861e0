"""The loop's temporal-reuse stage: `dpmhw.reconstruct.reuse.TemporalReuse` driven by the live settings.

The loop owns one history for its render size; a change of alpha, mode or split screen from
the operator takes effect on the next frame. A mode change resets the history (the two modes
fetch history from different places), so does `reset()` (operator request, or projection
resuming after a dark spell: that history shows another moment).
"""

from __future__ import annotations

import numpy as np

from dpmhw.reconstruct.reuse import ReuseSettings, TemporalReuse

__all__ = ["ReuseStage"]


class ReuseStage:
    def __init__(self, width: int, height: int, warmup: bool = False):
        self.warmup = warmup
        self.reuse = TemporalReuse(width, height, alpha=0.2, mode="same-pixel", warmup=warmup)

    def reset(self) -> None:
        self.reuse.reset()

    def apply(self, frame, mode: str, alpha: float, split_screen: bool = False, poses=None, camera=None) -> np.ndarray:
        """(H, W, 3) float32 linear radiance to post-process (left half plain with `split_screen`)."""
        wanted = ReuseSettings(alpha, mode, self.warmup, split_screen)
        if wanted != self.reuse.settings:
            if wanted.mode != self.reuse.settings.mode:
                self.reuse.reset()
            self.reuse.settings = wanted
        return self.reuse.update_frame(frame, poses=poses, camera=camera)
