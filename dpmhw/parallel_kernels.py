"""Per-pixel parallel kernels that run on the calling thread alone below a pixel count: waking
numba's worker threads costs a fixed 100 µs or so (a 2-core Zen 3) that a call over fewer pixels
does not earn back. One compilation serves both: `numba.set_num_threads(1)` (the calling
thread's setting only) runs the parallel loop in one piece, as fast as a serial compilation of
the same loop, which would be a second cold compile of seconds. One threshold for every such
kernel: each writes its own pixels only, so the thread count never changes a result, and the
lightest of them (the reuse blend) sets the break-even that the heavier ones (the G-buffer's
attributes) reach sooner."""

from __future__ import annotations

from contextlib import contextmanager

import numba as nb

PARALLEL_MIN_PIXELS = 16384
SPAN_PX = 512  # pixels of one call of a kernel's serial span function


@nb.njit(cache=True)
def spans(n):
    """Spans of SPAN_PX pixels covering n pixels. A parallel kernel loops over spans, each one
    call of a serial function: numba types and lowers a parallel loop's body twice (the loop,
    then its gufunc), so the body is kept to a call, and the per-pixel work is compiled once.
    The same bits as the loop in the body for IEEE kernels (the reuse's); with fast-math
    reassociation LLVM rounds a function optimised apart otherwise (the upsampling's last bit
    moved on 1 % of its values), so those keep their loops."""
    return (n + SPAN_PX - 1) // SPAN_PX


@nb.njit(cache=True)
def span(s, n):
    """Pixels [first, end) of span s of n."""
    return s * SPAN_PX, min(n, (s + 1) * SPAN_PX)


class PixelKernel:
    """`PixelKernel(py_func)(pixels, *args)`: py_func's parallel compilation on `args`, on this
    thread alone when `pixels` < PARALLEL_MIN_PIXELS."""

    def __init__(self, py_func):
        self.dispatcher = nb.njit(parallel=True, cache=True, nogil=True)(py_func)

    def __call__(self, pixels: int, *args):
        if pixels >= PARALLEL_MIN_PIXELS:
            return self.dispatcher(*args)
        with kernel_threads(1):
            return self.dispatcher(*args)


@contextmanager
def kernel_threads(n: int):
    """Parallel kernels this thread launches inside the block run on n of numba's threads (at
    most its pool's): the calling thread's own setting, put back after, also on a raise."""
    before = nb.get_num_threads()
    nb.set_num_threads(min(n, nb.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        nb.set_num_threads(before)
