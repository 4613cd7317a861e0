"""Per-pixel kernels compiled twice, serial and parallel, and the pixel count from which the
parallel one pays: waking numba's worker threads costs a fixed few tens of microseconds that a
call over fewer pixels does not earn back. One threshold for every such kernel: each writes its
own pixels only, so which compilation runs never changes a result, and the lightest of them
(the reuse blend) sets the break-even that the heavier ones (the G-buffer's attributes) reach
sooner."""

from __future__ import annotations

import types

import numba as nb

PARALLEL_MIN_PIXELS = 16384


def serial_and_parallel(py_func):
    """(serial, parallel) compilations of `py_func`, indexed by `pixels >= PARALLEL_MIN_PIXELS`;
    the serial one is a renamed copy so that the two never share an on-disk cache entry."""
    serial = types.FunctionType(py_func.__code__, py_func.__globals__, py_func.__name__ + "_serial")
    serial.__qualname__ = py_func.__qualname__ + "_serial"
    return nb.njit(cache=True, nogil=True)(serial), nb.njit(parallel=True, cache=True, nogil=True)(py_func)
