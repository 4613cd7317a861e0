"""A render of N passes as blocks of passes that can run anywhere, summed in one fixed order.

The integrator accumulates a frame's passes inside its kernels, in float32, into one film, so
the order in which it adds samples cannot be recreated from parts rendered elsewhere. A render
that may be split is therefore defined by its blocks instead:

- block b holds passes [8b, 8b + 8) (the last one may be shorter) and is one ordinary render,
  `PathIntegrator.render(seed=block_seed(S, b), spp=len)`: block 0 uses the render's own seed,
  so a render of at most 8 passes is exactly `render(seed=S, spp=N)`; the other blocks' seeds
  come from numpy's SeedSequence (independent streams, far from the small seeds of 1-spp frames);
- the image is Σ_b radiance_b · spp_b / Σ_b spp_b, accumulated in float64 in block order and
  rounded once to float32; the G-buffer (object ids) is block 0's.

The block size and the seeds never depend on how many machines run the blocks, nor on the
order in which they finish, so every executor gives the same image bit for bit. Only the public
render API is used (scene, time, seed, spp), so the renderer can change underneath.
"""

from __future__ import annotations

import time as _time
from dataclasses import dataclass
from typing import Callable

import numpy as np

PASSES_PER_BLOCK = 8  # a task's worth: long next to its overhead, short enough to balance many workers


@dataclass(frozen=True)
class Block:
    index: int
    first_pass: int  # of the whole render (for progress and metadata)
    passes: int
    seed: int


@dataclass
class BlockResult:
    index: int
    spp: int  # passes done (fewer than asked only if the render was stopped)
    radiance: np.ndarray  # (H, W, 3) float32: this block's mean
    nonfinite_samples: int
    object_id: np.ndarray | None  # block 0 only: the G-buffer comes from the render's own seed
    seconds: float  # wall time
    cpu_seconds: float  # CPU time of the process that rendered it, all its threads


def block_seed(seed: int, index: int) -> int:
    """Block 0 keeps the render's seed; block b > 0 gets a 63-bit seed from SeedSequence(seed, b)."""
    if index == 0:
        return int(seed)
    hi, lo = np.random.SeedSequence(int(seed), spawn_key=(int(index),)).generate_state(2, np.uint32)
    return ((int(hi) << 32) | int(lo)) & ((1 << 63) - 1)


def plan(seed: int, spp: int, block_passes: int = PASSES_PER_BLOCK) -> list[Block]:
    if spp < 1:
        raise ValueError(f"spp must be ≥ 1, got {spp}")
    return [Block(b, first, min(block_passes, spp - first), block_seed(seed, b))
            for b, first in enumerate(range(0, spp, block_passes))]


def render_block(integrator, time: float, block: Block, progress: Callable[[int, int], None] | None = None,
                 should_stop: Callable[[], bool] | None = None) -> BlockResult:
    started, cpu = _time.perf_counter(), _time.process_time()
    frame = integrator.render(time=time, seed=block.seed, spp=block.passes, progress=progress, should_stop=should_stop)
    return BlockResult(block.index, frame.spp, frame.radiance, frame.nonfinite_samples,
                       frame.object_id if block.index == 0 else None, _time.perf_counter() - started,
                       _time.process_time() - cpu)


class PassSum:
    """Folds block results into the image in block order, whatever order they arrive in; a
    block waits until all blocks before it are in. Stopping early keeps the folded prefix."""

    def __init__(self, blocks: list[Block]):
        self.blocks = blocks
        self.spp = 0
        self.nonfinite_samples = 0
        self.object_id: np.ndarray | None = None
        self.block_seconds: list[float] = []
        self.block_cpu_seconds: list[float] = []
        self._acc: np.ndarray | None = None
        self._waiting: dict[int, BlockResult] = {}
        self._next = 0

    @property
    def complete(self) -> bool:
        return self._next == len(self.blocks)

    @property
    def folded_blocks(self) -> int:
        return self._next

    def add(self, result: BlockResult) -> None:
        if result.index < self._next or result.index in self._waiting:
            raise ValueError(f"block {result.index} was already added")
        self._waiting[result.index] = result
        while self._next in self._waiting:
            r = self._waiting.pop(self._next)
            weighted = r.radiance.astype(np.float64) * r.spp  # exact: float32 × small integer
            self._acc = weighted if self._acc is None else self._acc + weighted
            self.spp += r.spp
            self.nonfinite_samples += r.nonfinite_samples
            self.block_seconds.append(r.seconds)
            self.block_cpu_seconds.append(r.cpu_seconds)
            if r.index == 0:
                self.object_id = r.object_id
            self._next += 1
            if r.spp < self.blocks[r.index].passes:  # stopped inside this block: nothing after it counts
                self._next = len(self.blocks)
                self._waiting.clear()

    @property
    def radiance(self) -> np.ndarray:
        if self._acc is None:
            raise ValueError("no block has been folded yet")
        return (self._acc / self.spp).astype(np.float32)


def render_local(integrator, time: float, seed: int, spp: int, progress: Callable[[int, int], None] | None = None,
                 should_stop: Callable[[], bool] | None = None) -> PassSum:
    """All blocks one after another on `integrator` (this process). `progress(done, spp)` after
    every pass; `should_stop` is polled between passes, and the sum then holds the finished ones."""
    blocks = plan(seed, spp)
    total = PassSum(blocks)
    for block in blocks:
        if should_stop is not None and total.spp > 0 and should_stop():
            break
        on_pass = None if progress is None else (lambda done, _n, first=block.first_pass: progress(first + done, spp))
        total.add(render_block(integrator, time, block, on_pass, should_stop))
        if total.complete:
            break
    return total
