"""PixelKernel: one parallel compilation, run on the calling thread alone below the threshold."""

import numba as nb
import numpy as np
import pytest

from dpmhw.parallel_kernels import PARALLEL_MIN_PIXELS, PixelKernel


def _scaled_py(x, out):
    if x.shape[0] and x[0] < 0.0:
        raise ValueError("negative")
    for i in nb.prange(x.shape[0]):
        out[i] = 2.0 * x[i]


def _threads_py(out):
    for i in nb.prange(out.shape[0]):
        out[i] = nb.get_thread_id()


scaled = PixelKernel(_scaled_py)
threads_seen = PixelKernel(_threads_py)


def test_small_calls_run_on_one_thread_and_give_the_large_calls_results():
    n = PARALLEL_MIN_PIXELS * 2
    ids = np.full(n, -1, np.int64)
    threads_seen(PARALLEL_MIN_PIXELS - 1, ids)  # the pixel count decides, not the array
    assert (ids == 0).all()
    x = np.linspace(0.0, 1.0, n)
    small, large = np.empty(n), np.empty(n)
    scaled(1, x, small)
    scaled(n, x, large)
    assert np.array_equal(small, large) and np.array_equal(large, 2.0 * x)


@pytest.mark.skipif(nb.config.NUMBA_NUM_THREADS < 2, reason="one thread: nothing to put back")
def test_the_thread_count_is_put_back_after_a_small_call_even_when_it_raises():
    before = nb.config.NUMBA_NUM_THREADS
    nb.set_num_threads(before)
    with pytest.raises(ValueError, match="negative"):
        scaled(1, np.array([-1.0, 1.0]), np.empty(2))
    assert nb.get_num_threads() == before
    threads_seen(PARALLEL_MIN_PIXELS, np.empty(4, np.int64))
    assert nb.get_num_threads() == before
