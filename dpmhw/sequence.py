"""Rendering a scene's timeline frame by frame through temporal reuse, and scaled-down scenes.

Frame k of a sequence starting at timeline frame f0 is rendered at t = (f0 + k) / fps with seed
seed0 + k and the scene's scripted poses at t; every reuse instance sees the same frames.
"""

from __future__ import annotations

import dataclasses
import time as _time
from dataclasses import dataclass
from typing import Callable, Iterator, Sequence

import numpy as np

from dpmhw.render.frame import Frame
from dpmhw.reconstruct.reuse import TemporalReuse
from dpmhw.scene_file import Scene


def scaled_scene(scene: Scene, scale: float) -> Scene:
    """The same scene rendered at `scale` × its resolution (at least 1 px), for quick runs."""
    r = scene.render
    return scene.at_size(max(1, round(r.width * scale)), max(1, round(r.height * scale)))


def with_fps(scene: Scene, fps: float) -> Scene:
    """The same scene on a timeline of `fps` frames per second."""
    return dataclasses.replace(scene, render=dataclasses.replace(scene.render, fps=float(fps)))


@dataclass
class SequenceStep:
    index: int  # k, 0-based within the sequence
    time: float
    frame: Frame
    outputs: list[np.ndarray]  # one per reuse instance, (H, W, 3) float32 linear
    render_ms: float
    reuse_ms: list[float]


def run_sequence(integrator, scene: Scene, frames: int, reusers: Sequence[TemporalReuse], seed: int = 0, start_frame: float = 0,
                 spp: int = 1, should_stop: Callable[[], bool] | None = None) -> Iterator[SequenceStep]:
    """Render `frames` frames of the timeline and pass each through every reuse instance."""
    fps = scene.render.fps
    camera = integrator.camera
    for k in range(frames):
        if should_stop is not None and k > 0 and should_stop():
            return
        t = (start_frame + k) / fps
        poses = scene.object_poses(t)
        t0 = _time.perf_counter()
        frame = integrator.render(time=t, seed=seed + k, spp=spp, poses=poses)
        render_ms = (_time.perf_counter() - t0) * 1e3
        outputs, reuse_ms = [], []
        for r in reusers:
            t0 = _time.perf_counter()
            outputs.append(r.update_frame(frame, poses, camera))
            reuse_ms.append((_time.perf_counter() - t0) * 1e3)
        yield SequenceStep(k, t, frame, outputs, render_ms, reuse_ms)
