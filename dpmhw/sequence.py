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
    """The same scene rendered at `scale` × its resolution (intrinsics scaled about the
    pixel-centre convention: c' = (c + 0.5)·s − 0.5), for quick runs."""
    if scale == 1:
        return scene
    r = scene.render
    width, height = max(1, round(r.width * scale)), max(1, round(r.height * scale))
    sx, sy = width / r.width, height / r.height
    K = np.array(scene.camera.K, dtype=np.float64, copy=True)
    K[0, 0], K[0, 1], K[0, 2] = K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5
    K[1, 1], K[1, 2] = K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5
    return dataclasses.replace(scene, render=dataclasses.replace(r, width=width, height=height),
                               camera=dataclasses.replace(scene.camera, K=K))


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
